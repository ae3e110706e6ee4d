// node-opcua's client as the OPC UA tests' second client stack (the tests' own peer; client side
// only). One JSON argument says whom to reach, how, and what to do; one JSON object on stdout says
// what happened, with OPC UA status codes by name, for the pytest test to assert on.
//
//   node peer.mjs '{"url": ..., "mode": "SignAndEncrypt", "policy": "Basic256Sha256",
//                   "cert": "client.pem", "key": "client_key.pem", "pki": "/tmp/...",
//                   "applicationUri": "urn:...", "user": "olga", "password": "...",
//                   "steps": [{"do": "session"}, ...]}'
//
// Nodes are named by browse paths from the Objects folder, each name prefixed by a namespace
// alias: "mv:" (Machine Vision), "mvpose:" (mvpose's own) or "0:"; "Server" is i=2253.
// Steps: endpoints, session (else opened by the first step that needs one), read, call,
// subscribe, wait_events. A failed step ends the run with
// "error" naming the step and the status; the results so far are printed.

import {
    AttributeIds, ClientMonitoredItem, ClientSubscription, DataType, MessageSecurityMode,
    OPCUAClient, SecurityPolicy, TimestampsToReturn, UserTokenType,
    Variant, constructEventFilter, makeBrowsePath, ofType, promoteOpaqueStructure,
    resolveNodeId,
} from "node-opcua-client";
import { readFileSync } from "node:fs";
import { OPCUACertificateManager } from "node-opcua-certificate-manager";  // node-opcua-client's own

const spec = JSON.parse(process.argv[2]);
const out = { results: [] };
const URIS = { mv: "http://opcfoundation.org/UA/MachineVision", mvpose: "urn:mvpose:opcua" };

function jsonable(value) {
    if (value === null || value === undefined) return null;
    if (value instanceof Date) return value.toISOString();
    if (Buffer.isBuffer(value)) return value.toString("hex");
    if (Array.isArray(value) || ArrayBuffer.isView(value)) return Array.from(value, jsonable);
    if (value instanceof Variant) return jsonable(value.value);
    if (typeof value === "bigint") return Number(value);
    if (typeof value === "object") {
        if (typeof value.toJSON === "function" && value.constructor?.name !== "Object") {
            const j = value.toJSON();
            return typeof j === "object" ? jsonable(j) : j;
        }
        if (value.schema || value.constructor?.schema) {
            const o = {};
            for (const f of (value.schema || value.constructor.schema).fields) o[f.name] = jsonable(value[f.name]);
            return o;
        }
        const o = {};
        for (const [k, v] of Object.entries(value)) o[k] = jsonable(v);
        return o;
    }
    return value;
}

let client, session, namespaces;
const subscriptions = {};

async function ns(alias) {
    if (alias === "0") return 0;
    if (!namespaces) {
        const dv = await session.read({ nodeId: "i=2255", attributeId: AttributeIds.Value });
        namespaces = dv.value.value;
    }
    const i = namespaces.indexOf(URIS[alias]);
    if (i < 0) throw new Error(`the server has no namespace ${URIS[alias]}`);
    return i;
}

async function qualified(name) {
    const [alias, local] = name.includes(":") ? name.split(":", 2) : ["0", name];
    return `${await ns(alias)}:${local}`;
}

async function resolve(path, from = "ObjectsFolder") {
    if (path === "Server") return resolveNodeId("i=2253");
    const parts = [];
    for (const name of path) parts.push(await qualified(name));
    const r = await session.translateBrowsePath(makeBrowsePath(from, "/" + parts.join("/")));
    if (!r.statusCode.isGood() || !r.targets?.length) {
        throw new Error(`browse path ${JSON.stringify(path)}: ${r.statusCode.name}`);
    }
    return r.targets[0].targetId;
}

function variant(arg) {
    if (arg.type === "Null") return new Variant({ dataType: DataType.Null });
    return new Variant({ dataType: DataType[arg.type], value: arg.value,
                         arrayType: arg.array ? 1 : undefined });
}

async function openSession() {
    const identity = spec.user
        ? { type: UserTokenType.UserName, userName: spec.user, password: spec.password }
        : { type: UserTokenType.Anonymous };
    session = await client.createSession(identity);
}

async function step(s) {
    if (!session && !["endpoints", "session"].includes(s.do)) await openSession();
    switch (s.do) {
    case "endpoints": {
        const eps = await client.getEndpoints();
        return eps.map((e) => [e.securityPolicyUri.split("#").pop(), MessageSecurityMode[e.securityMode]]);
    }
    case "session":
        await openSession();
        return "ok";
    case "read": {
        const dv = await session.read({ nodeId: await resolve(s.path), attributeId: AttributeIds.Value });
        if (!dv.statusCode.isGood()) return { status: dv.statusCode.name };
        await promoteOpaqueStructure(session, [dv]);
        return { status: dv.statusCode.name, value: jsonable(dv.value.value) };
    }
    case "call": {
        const objectId = await resolve(s.object);
        const methodId = await resolve([s.method], objectId);
        const r = await session.call({ objectId, methodId, inputArguments: s.args.map(variant) });
        return { status: r.statusCode.name,
                 inputArgumentResults: (r.inputArgumentResults || []).map((c) => c.name),
                 outputs: (r.outputArguments || []).map((v) => jsonable(v.value)) };
    }
    case "subscribe": {
        const sub = ClientSubscription.create(session, {
            requestedPublishingInterval: 50, requestedLifetimeCount: 600, requestedMaxKeepAliveCount: 20,
            maxNotificationsPerPublish: 1000, publishingEnabled: true, priority: 1 });
        const fields = [];
        for (const f of s.fields) fields.push(await qualified(f));
        const type = s.ofType === "BaseEventType" ? resolveNodeId("i=2041")
            : s.ofType ? await resolve(s.ofType, "i=2041") : null;  // a path under BaseEventType
        const filter = constructEventFilter(fields, type ? ofType(type) : undefined);
        const item = ClientMonitoredItem.create(sub, {
            nodeId: await resolve(s.node), attributeId: AttributeIds.EventNotifier,
        }, { filter, queueSize: 1000, discardOldest: false }, TimestampsToReturn.Both);
        const got = { events: [], pending: [] };
        item.on("changed", (values) => {
            got.pending.push((async () => {
                const dvs = values.map((v) => ({ value: v }));
                await promoteOpaqueStructure(session, dvs);
                const ev = {};
                s.fields.forEach((f, i) => { ev[f] = jsonable(dvs[i].value.value); });
                got.events.push(ev);
            })());
        });
        await new Promise((ok, fail) => {
            item.once("initialized", ok);
            item.once("err", (e) => fail(new Error(`monitored item: ${e}`)));
        });
        subscriptions[s.label] = got;
        return "ok";
    }
    case "wait_events": {
        const got = subscriptions[s.label];
        const deadline = Date.now() + (s.timeout_ms ?? 30000);
        while (got.events.length < s.count && Date.now() < deadline) {
            await new Promise((r) => setTimeout(r, 20));
        }
        await Promise.all(got.pending);
        return got.events;
    }
    default:
        throw new Error(`unknown step ${s.do}`);
    }
}

// node-opcua's client will not open a session on a security mode the server does not offer; a
// client that insists (as an attacker's would) takes an offered endpoint and claims it has ours;
// with "serverCert" (the server's DER) it also opens a secure channel of any mode unchecked.
async function insist() {
    const offered = await client.getEndpoints();
    const own = client.findEndpoint.bind(client);
    client.findEndpoint = (url, mode, policy) => own(url, mode, policy) ?? Object.assign(
        Object.create(Object.getPrototypeOf(offered[0])), offered[0],
        { securityMode: mode, securityPolicyUri: policy });
    client.findEndpointForSecurity = (mode, policy) => client.findEndpoint("", mode, policy);
}

async function main() {
    const pki = new OPCUACertificateManager({ rootFolder: spec.pki, automaticallyAcceptUnknownCertificate: true });
    await pki.initialize();
    client = OPCUAClient.create({
        applicationName: "mvpose node-opcua peer", applicationUri: spec.applicationUri,
        securityMode: MessageSecurityMode[spec.mode], securityPolicy: SecurityPolicy[spec.policy],
        certificateFile: spec.cert, privateKeyFile: spec.key, clientCertificateManager: pki,
        endpointMustExist: false, connectionStrategy: { maxRetry: 0, initialDelay: 100 },
        // known up front, node-opcua opens the channel without checking the offered endpoints
        serverCertificate: spec.insist && spec.serverCert ? readFileSync(spec.serverCert) : undefined,
        requestedSessionTimeout: 120000,
        defaultTransactionTimeout: 120000,  // a call held inside the station (a test) waits
    });
    try {
        await client.connect(spec.url);
        out.connected = true;
        if (spec.insist) await insist();
    } catch (err) {
        out.connected = false;
        out.error = `connect: ${err.message}`;
        return;
    }
    try {
        for (const s of spec.steps) {
            try {
                out.results.push(await step(s));
            } catch (err) {
                out.error = `${s.do}: ${err.message}`;
                return;
            }
        }
    } finally {
        if (session) await session.close().catch(() => {});
        await client.disconnect().catch(() => {});
    }
}

main().then(() => {
    process.stdout.write(JSON.stringify(out) + "\n");
    process.exit(0);
}, (err) => {
    process.stdout.write(JSON.stringify({ ...out, error: `peer: ${err.stack}` }) + "\n");
    process.exit(0);
});
